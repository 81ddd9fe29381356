"""uacell: an OPC UA server for OPC 40010-1 Robotics and OPC 30050 PackML remote operation."""

__version__ = "0.1.0"
