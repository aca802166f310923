"""closedloop.io."""
