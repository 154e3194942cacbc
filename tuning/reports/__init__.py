"""The trust reports behind ``diffpen report`` and ``diffpen bench``, one module per concept:

* :mod:`tuning.reports.reference`: independent reference solutions (closed forms, DOP853 with
  located contact events) and the measurements of sampled trajectories compared with them;
* :mod:`tuning.reports.extreme`: the extreme-case stability matrix (``diffpen report
  stability``);
* :mod:`tuning.reports.accuracy`: error against run time of every integrator, the cheapest one
  that meets a tolerance, and the work-precision plot (``diffpen report accuracy``);
* :mod:`tuning.reports.gradient_check`: gradient error against dt and smoothing width
  (``diffpen report gradients``), and through contact events against the event-located ball;
* :mod:`tuning.reports.box_gradients`: a box landing on a corner, derivatives w.r.t. k, c
  and mu against :class:`~tuning.reports.reference.BoxCornerReference`;
* :mod:`tuning.reports.bench`: speed against baselines measured in the same process
  (``diffpen bench``): its cases and how they are run; :mod:`tuning.reports.floors`, the
  hand-written baselines; :mod:`tuning.reports.timing`, medians of calls taken in turns.

They compute and return plain data; ``tuning.cli.report`` and ``tuning.cli.bench`` print. The
package imports its modules lazily: import the one you need.
"""
