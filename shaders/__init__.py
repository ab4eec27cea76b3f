"""What the shaders compute: the SG math reference, the node-group formula and its node builder, octahedral maps,
the OSL light-field camera, environment visibility, and the quadratures that check the closed forms.

Imports need only numpy; never bpy or torch."""
