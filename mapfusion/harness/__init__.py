"""The harness: the layer above the engine (:mod:`mapfusion`) and the simulator (:mod:`sim`).

Run, batch, sweep, tune, calibration, stress, bench, plots, the result tables and the
``mapfusion`` command live here. It owns files, progress and printing; the engine below it
takes measurements and returns estimates, and never imports this package or :mod:`sim`.
"""
