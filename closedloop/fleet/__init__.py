"""closedloop.fleet."""
