"""Rotation groups: SO(3) (:mod:`.so3`, closed forms) and SO(n) (:mod:`.son`, any rank).

Both are batched over leading dimensions, differentiable, and finite in value and gradient at
the rotation angles 0 and π. ``son`` defers to ``so3`` for n = 3; ``so3`` never imports ``son``.
"""
from . import so3, son

__all__ = ["so3", "son"]
