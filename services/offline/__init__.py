"""The offline front doors, no Zenoh: ``vistrack track`` and ``vistrack tune`` run exactly the
code the services run, over recorded frames."""
