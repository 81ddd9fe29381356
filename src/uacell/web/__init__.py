"""The browser HMI: an OPC UA client of the server that shows the cell live (docs/web.md).

``uacell.web.hosting.start_web`` runs it; ``uacell.web.discovery`` finds the cell by type and
BrowseName; ``uacell.web.uasession`` is one web user's OPC UA session; ``uacell.web.app`` the HTTP side.
"""
