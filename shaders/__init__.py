"""numpy side of SG Lightfield: SG math reference, octahedral maps, quadrature, EXR I/O.

Imports need only numpy (and OpenEXR for ``exr_io``); never bpy or torch."""
