"""Frames made on a Ray cluster (``render_backend = "ray"``), built on server/stream/:
``backend`` is :class:`RayWorkers`, the stream's FrameWorkers for render-worker actors,
``pool`` the gateway's render workers (placement by load, fair share, failover), ``worker``
the actor (the stream's SceneFrames), ``notices`` what participants are told when their
worker is lost, ``routes`` the placement endpoint.
"""
