"""OPC 10000-100 DI: the device root and LockingServices, as a uacell companion."""
