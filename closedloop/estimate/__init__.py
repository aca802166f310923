"""closedloop.estimate."""
