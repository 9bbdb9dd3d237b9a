"""Warp kernels. ``fem``: per-quadrature-point energy, force and Hessian assembly;
``linalg``: vector and block-sparse operations used by the solvers."""
