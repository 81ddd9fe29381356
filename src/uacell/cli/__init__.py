"""The `uacell` command line: serve, health, config check, models, nodeset, user, cert (main.py)."""
