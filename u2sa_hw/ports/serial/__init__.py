"""The serial port kind (docs/ports.md): its address grammar, backends, mock client and wire protocol."""
