"""OPC 40001-1 Machinery (Basic Building Blocks) as a uacell companion: every robot and PackML unit of
the cell is a machine in ``Objects/Machines`` with its identification, MachineryItemState and
MachineryOperationMode (docs/machinery.md)."""
