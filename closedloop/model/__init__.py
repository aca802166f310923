"""closedloop.model."""
