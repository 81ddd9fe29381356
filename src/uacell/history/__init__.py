"""History: what happened on the line (OPC 10000-11 HistoryRead of values and events).

``store.py`` keeps samples (one table keyed by node, written in batches by a writer thread);
``backends.py`` holds the SQLite backend (embedded, default) and the PostgreSQL one;
``cursor.py`` the opaque continuation points; ``processed.py`` the aggregates (pure);
``service.py`` wires it into asyncua's HistoryRead service. docs/history.md says how it behaves.
"""
