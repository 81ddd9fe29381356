"""The asyncua adapter: the one door to asyncua and uvicorn (door/: every patch, swap, subclass and
private read, its inventory and version check; docs/asyncua.md), the request pipeline, the binary
codecs, NodeSet loading and the address-space snapshot. Nothing outside it reaches past asyncua's
public surface (tests/test_asyncua_door.py)."""
