"""Old name of `stdr.train.optim` (adam_step, clear_grads), kept working: stdr/_moved.py."""
from .._moved import alias
from .optim import adam_step, clear_grads  # noqa: F401

alias(__name__, "stdr.train.optim", {})
