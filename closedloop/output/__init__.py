"""closedloop.output."""
