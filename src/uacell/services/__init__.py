"""Server services beside the companions: diagnostics, the audit observers, the Prometheus metrics and
the registration with a discovery server."""
