"""Starting the system: ``vistrack up`` (the launch file and the process supervisor), the
Zenoh router, the demo, and the certificates for multi-host deployments."""
