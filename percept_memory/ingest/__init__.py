"""Ways in: everything that brings percepts into the memory."""
