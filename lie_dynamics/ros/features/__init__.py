"""Per-sample features of the dynamics node behind one interface (base.py). The logic of each is
plain Python; its rclpy side, where it has one, is a module of its own (contact_topics, gravity_payload)."""
