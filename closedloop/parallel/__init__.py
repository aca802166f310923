"""closedloop.parallel."""
