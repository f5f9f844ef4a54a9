"""Several drones, one map: a map server and drone clients that share a pose graph through deltas over ZeroMQ.

* :mod:`~slam2d.fleet.protocol`: the versioned msgpack messages and their checks;
* :mod:`~slam2d.fleet.journal`: the server's SQLite (WAL) state, one transaction per delta;
* :mod:`~slam2d.fleet.joint`: the joint pose graph, inter-robot loop closures, map tiles;
* :mod:`~slam2d.fleet.server`: the map server (ROUTER socket);
* :mod:`~slam2d.fleet.drone`: a simulated drone with its own lidar front end (DEALER socket).
"""
