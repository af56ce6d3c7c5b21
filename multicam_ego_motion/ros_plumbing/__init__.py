"""The base's ROS plumbing, shared by every node and tool: message conversions
(pose_messages; bearing_messages and imu_messages, read and written as CDR bytes by
wire_types), QoS profiles (qos), parameter declaration from tables (node_parameters), the
lean node and node entry point (lean_node, node_main), /diagnostics statuses (diagnostics),
DDS domain and transport set-up (ros_domain, dds_transport) and where the installed package's
shared files are (package_share)."""
