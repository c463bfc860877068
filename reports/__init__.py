"""Reports from the tracked studies: `python -m reports`. Loading studies from the MLflow store or
from the exports kept in the repository (data), one study's report folder with its tables and
figures (study_report), RESULTS.md from its template (results), the analyses across studies it
quotes (analyses); figure plumbing (plotting) and the paper's own numbers (paper).
"""
