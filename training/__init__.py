"""torch side of SG Lightfield: differentiable SG math, SG fitting, hair U-Net."""
