"""closedloop.loops.camera."""
