"""The central-difference check the gradient tests share."""

from __future__ import annotations


def assert_central_differences(checks, label="", *, tol=1e-5, value=None):
    """``checks``: {name: (analytic, f, h)} with f(h) the loss at the parameter moved by h (``value``
    picks the loss out of what f returns). Prints each relative error |analytic - fd| / |fd| of the
    central difference fd = (f(h) - f(-h)) / 2h and asserts every one <= ``tol``; returns them."""
    loss = value or (lambda r: r)
    errors = {}
    for name, (an, f, h) in checks.items():
        fd = (loss(f(h)) - loss(f(-h))) / (2 * h)
        errors[name] = abs(an - fd) / abs(fd)
    print(label, {k: f"{e:.1e}" for k, e in errors.items()})
    assert max(errors.values()) <= tol, errors
    return errors
