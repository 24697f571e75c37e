"""The sans-IO Modbus codec: checksums, PDUs of every function code, and framers.

Never imports socket, serial, time, click or rich (design notes, "The codec is sans-IO").
Importing this package registers every function code.
"""

from mbtool.codec import data_access  # noqa: F401  (registers FC 01-06, 15, 16)
