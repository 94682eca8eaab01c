"""ros2: the pipeline as ROS 2 topics over rmw_zenoh's wire format (see service.py)."""
