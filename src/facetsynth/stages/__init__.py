"""Stage runners: what each workflow rule does, from input files to output files.

Each runner reads its inputs, calls the numerical modules of the package and
writes its outputs atomically. The Snakemake scripts in ``workflow/scripts``
only unpack the ``snakemake`` object and call one of these; the CLI and the
tests call them directly.
"""
