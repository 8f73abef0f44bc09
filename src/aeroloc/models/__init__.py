"""Model registries: ``retrieval`` (global descriptors) and ``local`` (keypoints, descriptors, matchers)."""
