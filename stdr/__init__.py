"""stdr: dynamic-scene reconstruction with deformable 3D Gaussian Splatting and STDR."""

__version__ = "0.1.0"
