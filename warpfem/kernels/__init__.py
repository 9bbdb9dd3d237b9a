"""Warp kernels. ``fem``: per-quadrature-point energy, force and Hessian assembly;
``linalg``: vector and block-sparse operations used by the solvers; ``warping``: stiffness warping;
``subspace``: cubature forces and reconstruction of subspace (model-reduced) simulation;
``structs``: the Warp structs that bundle the arguments the quadrature-point (and warping) kernels share.

Vocabulary: "subspace" is model reduction (x = X + U q); "selective reduced integration" (SRI) is
the Hex8 quadrature with a separate one-point volumetric set (``QuadratureData.volumetric``)."""
