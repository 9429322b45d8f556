"""What each robot is told to do: the operator's orders (operator) and the arbiter that picks
the behaviour driving a robot now — held, an errand, looking, a meeting, a sweep stop, or
exploring — and has the driver (``server.control``) make its twist (steering)."""
