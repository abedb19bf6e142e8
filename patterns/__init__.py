"""patterns: printer profiles, G-code writing and parsing, the motion planner, test patterns and manifests."""
