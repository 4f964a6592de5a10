"""One router per resource of the pod's HTTP API."""
