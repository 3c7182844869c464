"""What users run outside the workflow: the facetsynth command, prediction, previews, summaries, the report's
figures and the benchmarks.
"""
