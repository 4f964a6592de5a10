"""One router per resource: pods, job, routing, health (with metrics)."""
