"""closedloop.validation."""
