"""flowins: optical-flow assisted inertial navigation, differentiable, in PyTorch."""

__version__ = "0.1.0"
