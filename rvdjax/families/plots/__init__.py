"""Each family's run figure, one module per family, apart from the kernel's modules."""
