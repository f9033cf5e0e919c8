"""An independent model of ROS 2 rmw_zenoh 0.10.5 / 0.12.0 (the rosidl::Buffer era) on the wire.

Written from upstream's released C++ sources alone (see README.md in this folder), on plain
``zenoh``, ``xxhash`` and ``rosbags``; it imports nothing of the project it is used to test.
Run a model participant as ``python -m tests.upstream_model <role> ...`` (see ``__main__``).
"""
