"""mbtool: a command-line Modbus master."""

__version__ = "0.1.0"
