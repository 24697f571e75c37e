"""Master side I/O: transports, the client (time, retries, id matching), connections, the poll loop."""
