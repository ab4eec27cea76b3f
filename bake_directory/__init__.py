"""The bake directory: what each stage writes and the next one reads (plan, texel maps, light-field tiles, SG
textures, report), with atomic writes and plan-hash checks. docs/architecture.md, "The bake directory is the contract".

Imports need only numpy (OpenEXR for EXR files, Pillow for pictures, flip-evaluator for FLIP); never bpy or torch."""
