"""The plant: every device of several links, polled from one process (mbtool poll)."""
