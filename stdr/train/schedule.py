"""Old name of `stdr.train.optim.exp_lr` (the learning-rate schedule), kept working: stdr/_moved.py."""
from .._moved import alias
from .optim import exp_lr  # noqa: F401

alias(__name__, "stdr.train.optim", {})
