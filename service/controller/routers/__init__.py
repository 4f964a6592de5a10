"""One router per resource: pods, job, routing (health and metrics: ``service.routers``)."""
