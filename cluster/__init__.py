"""credit's application package. Importing it sets one process-wide default before torch
loads: OpenMP threads that sleep when idle rather than spin (`cluster.cpu`)."""

from cluster.cpu import prefer_sleeping_threads

prefer_sleeping_threads()
