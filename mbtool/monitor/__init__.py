"""The passive bus monitor: frames split from a bus's bytes, and pcap captures."""
