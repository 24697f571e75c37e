"""SunSpec: a device that describes itself (issue 34).

Most solar inverters, their meters and batteries hold the marker "SunS" at holding
register 40000 (or 0, or 50000), then a chain of models, each its id and its length,
ending with the end model 0xFFFF.  The SunSpec Alliance's model definitions (``models/``,
Apache-2.0) say what each model's registers are: with them the chain names every point,
with its type, unit and scale factor, and no map needs to be written by hand.

``models`` reads the definitions; ``layout`` lays a model's definition over its registers
(the repeating groups counted, the quirks of real devices named); ``discover`` walks a
device's chain with the reads it is given.  The values are the register map's own
(``registermap``): a discovered model is a map, so ``mbtool sunspec`` and ``read -m`` of
the map it writes cannot disagree.
"""
