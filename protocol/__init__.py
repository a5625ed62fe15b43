"""Wire protocol shared by server and clients: message types, msgpack codec, limits.

Filled in by the streaming-service issue; it may import numpy, msgpack and pydantic only.
"""
