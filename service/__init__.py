"""HTTP side of the service: the FastAPI app (service.app), its routes and the one-machine
mode that starts Redis and a worker (service.embedded)."""
