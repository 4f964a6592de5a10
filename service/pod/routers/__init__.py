"""One router per resource of the pod's HTTP API (health and metrics: ``service.routers``)."""
