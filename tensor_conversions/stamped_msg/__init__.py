"""The ``.msg`` files of ROS package ``warp_buffer_msgs`` (announced through the
``rosidl_buffer.interfaces`` entry points): ``warp_buffer_msgs/msg/StampedTensor``, an
ExperimentalTensor with the header upstream's message lacks (see docs/examples.md)."""
