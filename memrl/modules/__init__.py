"""Networks (Table I Q-network) and policies."""
