"""Inversion jobs: a jobs table with leases (the source of truth), huey as the queue, worker processes.

``JobSystem(settings)`` is what the app starts in its lifespan (``start()``/``stop()``); the
routers in :mod:`service.routers.jobs` use it to submit, read, list and cancel jobs.
"""

from service.jobs.system import JobSystem

__all__ = ["JobSystem"]
