"""Launchers: the in-process and Ray acting and data sides of the one loop (`cluster.loop`), the
buffer-service process and `credit cluster up`."""
