"""The differentiable renderer R: cameras, view layouts, rasterisation of meshes and points, shading."""
