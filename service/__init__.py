"""vecsim's HTTP services: the sim pod, the controller and the local job runner."""
