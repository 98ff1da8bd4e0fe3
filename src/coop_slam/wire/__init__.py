"""What crosses the radio between robots and the server.

- :mod:`.record`: the keyframe record the core computes with, and its validation.
- :mod:`.messages`: the messages as plain data, one class per ROS message (``msg/``).
- :mod:`.codec`: a record to the message of its kind and back (one encoder, one decoder per kind);
  :mod:`.encodings`, :mod:`.bow_signature`, :mod:`.pack` and :mod:`.varint` are the compact
  encodings it uses, :mod:`.observations` what an update changes.
- :mod:`.delivery`: numbered messages, taken in order once each, acknowledged, sent again.
- :mod:`.legacy`: keyframe messages of recorded runs, in the format before each kind had its own.

How each kind is laid out on the wire: ``docs/wire.md``.
"""
