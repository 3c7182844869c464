"""What users run outside the workflow: the facetsynth command, prediction, previews, summaries, the report's
figures and the benchmarks.
"""

from ..io.pages import memory_defaults

memory_defaults()   # the facetsynth command's numpy and the jobs it starts: io/pages.py
