"""Register maps: a device's points by name, with scaling, units, enums and bits (issue 15)."""
