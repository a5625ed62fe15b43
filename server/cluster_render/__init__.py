"""Where frames are made (``render_backend``): ``backend`` is the seam the stream and room
code goes through (local: this process's render threads; ray: render-worker actors), ``pool``
the gateway's render workers on a Ray cluster (placement by load, failover), ``worker`` the
actor, ``gateway`` a room's and a plain session's side of a scene on a worker, ``notices``
what participants are told when their worker is lost, ``routes`` the placement endpoint.
"""
