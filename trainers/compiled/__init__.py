"""The compiled path: the C kernel (``_kernel.c``), its build, ABI and loader, and the batch
state (``fast``)."""
