"""Per-sample features of the dynamics node behind one interface (base.py). The logic of each is
plain Python (contact, gravity_source, payload_service); the feature classes the node registers
hold the rclpy side (contact_topics, gravity_topic, payload_services, dynamics_topics); recording
holds both (its plain part: SampleLog and Recorder)."""
