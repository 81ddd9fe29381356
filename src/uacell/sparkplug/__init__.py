"""The cell as an Eclipse Sparkplug B 3.0 edge node on an MQTT broker, beside or instead of PubSub
(``[sparkplug]``, docs/sparkplug.md)."""
