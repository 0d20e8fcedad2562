"""Hardware abstraction: the Backend interface, a registry by name, and the backends."""
