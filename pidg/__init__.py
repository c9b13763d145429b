"""pidg: Physics-Informed Deformable Gaussian Splatting."""
from pidg import _env  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)

__version__ = "0.1.0"
