"""Built-in plugins. Each module registers through the ``teletouch`` entry-point group, like a third-party one."""
