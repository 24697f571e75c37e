"""The commands, one module per family of function codes."""
