"""A third companion that lives only in the tests (tests/test_third_companion.py): nothing outside
tests/ knows it. It gives every PackML unit a ``Thermometer`` with its ``Temperature`` and shows the
units in ``Objects/Thermometers``; see ``companion.py``."""
