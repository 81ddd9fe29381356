"""The binder toolkit: what a companion's binder uses to put its pure model on OPC UA nodes (Space's
typed operations, the one state-machine binding, the ordered publisher, the one method dispatcher,
client writes, the condition binding, the file directory, the cell's parts). It reaches asyncua only
through uacell.ua."""
