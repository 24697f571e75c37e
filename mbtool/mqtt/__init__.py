"""A plant on an MQTT broker: what ``mbtool poll`` reads, published as it is read.

The plant's ``Poll`` records, handed on by the thread that runs the plant, reach this room
through one entry point, ``publisher.MqttPublisher.report``, which only enqueues: publishing
never holds up a link's thread or the plant's output.  ``settings.py`` checks the ``[mqtt]``
table of an inventory (and ``--mqtt URL``); ``topics.py`` names the topics and writes the
payloads; ``change.py`` decides which points a poll publishes (on_change, deadband,
heartbeat); ``discovery.py`` writes Home Assistant's discovery configs; ``sparkplug.py`` is
Sparkplug B's edge node (``payload = "sparkplug_b"``); ``spool.py`` keeps QoS 1 messages
while the broker is away; ``writes.py`` checks a ``/set`` and makes the job a link's worker
runs; ``publisher.py`` runs the client (paho-mqtt, imported only when MQTT is used).
"""
