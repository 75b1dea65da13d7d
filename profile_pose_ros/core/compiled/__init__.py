"""The numba kernels (estimate, dense refinement, profile decoding, rendering), their status codes and
option layout, and which build of them a process runs (loader: prebuilt by aot, or JIT)."""
