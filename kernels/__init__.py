"""OpenCL kernels (*.cl), their host wrapper (program.py) and the kernel-host contract (contract.py)."""
