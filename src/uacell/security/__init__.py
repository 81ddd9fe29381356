"""Security of the server: certificates and endpoints, the trust list, logins and their throttle,
per-session rights, users, the audit trail (docs/security.md)."""
