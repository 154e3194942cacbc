"""The trust reports behind ``diffpen report`` live in one module per concept:

* :mod:`tuning.reference`: independent reference solutions (closed forms, DOP853 with located
  contact events) and the measurements of sampled trajectories compared with them;
* :mod:`tuning.extreme`: the extreme-case stability matrix (``diffpen report stability``);
* :mod:`tuning.accuracy`: error against run time of every integrator, the cheapest one that
  meets a tolerance, and the work-precision plot (``diffpen report accuracy``);
* :mod:`tuning.gradient_check`: gradient error against dt and smoothing width
  (``diffpen report gradients``).

``tuning.cli.report`` prints them. This module defines nothing.
"""
