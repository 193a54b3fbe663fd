"""The composition layer: functions that wire several capabilities (and the simulated lab) together.

``trajectories``, ``capture`` and ``estimation`` never import each other, and the core below them
never imports them. What needs two of them at once (the demo, flying on live VO, synthetic VO
sequences along the lab's flight patterns, a simulated lab session for a script) lives here, as
plain functions that take and return objects, so that the CLI, notebooks, benchmarks and tests
call the same code. ``flightkit/cli/`` parses arguments and calls one function from here.
"""
