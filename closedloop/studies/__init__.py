"""closedloop.studies."""
