"""What users run outside the workflow: the facetsynth command, prediction, previews, summaries, the report's
figures and the benchmarks.
"""

from ..io.pages import small_pages

small_pages()   # the facetsynth command's numpy, imported after this package, on small pages (io/pages.py)
