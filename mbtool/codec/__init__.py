"""The sans-IO Modbus codec: checksums, PDUs of every function code, and framers.

Never imports socket, serial, time, click or rich (design notes, "The codec is
sans-IO").  Function-code modules register themselves when imported;
``pdu.function_type`` imports a code's module (``pdu.FUNCTION_MODULES``) on the
code's first look-up, so a one-shot command pays only for the function codes it uses.
"""
