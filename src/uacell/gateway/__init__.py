"""Gateway to real equipment behind a PLC (issue 21, in progress).

Only the pure pieces exist so far: ``codec`` (Modbus register values with type, byte and word
order) and ``packtags`` (the default PackTags map under a prefix, every tag overridable). No
transport, driver or configuration hook uses them yet.
"""
