"""The asyncua-free kernel every layer builds on: the state machine, errors, roles and rights, the
companion declaration, DataSets, conditions, the cell as data, equipment factories and capabilities,
background tasks, logging, atomic files and the program file store (docs/architecture.md)."""
