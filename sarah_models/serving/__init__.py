"""The live agent: ``sarah-serve`` streams motion over WebSocket (docs/protocol.md).

``protocol.py`` is the wire format (one owner of every message's shape and check),
``server.py`` the server (one ``StreamingSession`` per connection, the browser page at ``/``),
``client.py`` a scripted client that writes the motion.npz ``sarah-generate`` writes.
"""
