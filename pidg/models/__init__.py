"""What a scene is made of: canonical Gaussians, deformation fields, the material field, the time axis, and the
scene model that composes them (``DynamicGaussians``)."""
