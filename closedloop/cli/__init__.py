"""closedloop.cli."""
