"""vecsim's HTTP services: the sim pod, the controller and the local job runner, with what they
share (``http``: middleware both servers mount; ``probes``: their probe paths and thresholds) and
the ``vecsim`` command (``cli``). Installed with the ``pod`` extra."""
