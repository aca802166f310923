"""closedloop.design."""
