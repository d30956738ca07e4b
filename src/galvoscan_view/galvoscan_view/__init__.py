"""galvoscan view: a Foxglove WebSocket bridge and a browser page on the running graph."""
