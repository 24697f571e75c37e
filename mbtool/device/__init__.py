"""The simulated device: data model, function handlers, data files, the server (``mbtool serve``)."""
