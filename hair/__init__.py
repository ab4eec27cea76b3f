"""The hair filter (Currius et al. 2022): a stochastic strand render filtered by a small U-Net through onnxruntime.

`raster`, `pairs` and `filtering` need numpy and onnxruntime only; `unet` and `train` need torch; `blender_scene`
needs bpy. Nothing here imports a submodule, so the package itself needs none of them."""
