"""Serial protocol between the Jetson and the Mecanum motor board (see PROTOCOL.md)."""
