"""closedloop.problem."""
