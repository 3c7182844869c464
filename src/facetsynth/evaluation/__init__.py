"""Scoring a fit against a virtual capture's truth, apart from the fit (issue 30).

A virtual capture (the virtual rig's, or one rendered by Mitsuba) names its true scene; a real capture has
none, and every scorer here returns ``{}`` for it. The stages call these after they have fitted and written
(load, fit, write, then score), and record the scores in their ``metrics.json`` under the keys they have
always had. The fit never reads the truth: the numerical core and the stages reach the scenes, the virtual
rig and the other renderers only through this package (``tests/test_import_rules.py``).

Modules, one per stage scored:

* :mod:`.truth`: the truth at the rectified points and the one rule for which points are scored
  (:func:`~.truth.analytic_points`, :func:`~.truth.scored_points`);
* :mod:`.hdr`: merged frames against the true radiance; :mod:`.rectify`: registration and rectified radiance;
* :mod:`.separate`: kd; :mod:`.partial_ndf`: partial NDFs against the recoverable true NDF, and the paper's
  variants compared (:func:`~.partial_ndf.variant_errors`);
* :mod:`.synthesize`: the completed NDFs at the points; :mod:`.params`: eta, ks and the NDF spread per
  homogeneous region; :mod:`.refine`: kd, ks, ks F0 and the spread of the delivered model.

Beside them, what scores a fit without a truth: :mod:`.metrics` (relative L2, PSNR, the measures every
score uses) and :mod:`.selfcheck` (the fit against its own capture's lights, issue 29). The held-out views
and lights (``validate``, ``selfcheck``) are stages of their own. Importing the package
imports none of its modules (the truth's among them): import the one you need.
"""
