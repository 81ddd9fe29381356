"""Equipment simulators to try the gateway with no PLC (run them as ``python -m``)."""
