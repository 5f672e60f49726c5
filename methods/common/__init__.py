"""Building blocks shared by methods (policy network, normalizer, BC loss)."""
