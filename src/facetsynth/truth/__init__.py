"""Ground truth: the scenes, the virtual rig that renders them, and the captures Mitsuba 3 renders. The fit never
imports this package (tests/test_import_rules.py); facetsynth.evaluation does.
"""
