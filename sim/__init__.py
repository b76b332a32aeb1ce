"""The simulation side of the test bed: SUMO networks and traffic, sensor models, scenarios.

``sim`` may import :mod:`mapfusion`; the reverse never happens.
"""
