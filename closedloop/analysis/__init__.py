"""closedloop.analysis."""
