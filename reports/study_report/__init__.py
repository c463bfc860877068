"""One study's report, reports/out/<study>/index.html (build, html with its templates/): Table I with its figure,
first (table_one, which RESULTS.md composes across studies), the ablation's tables (tables; the strict
pick-and-place criterion beside the lenient one: criteria) and figures (ablation_figures, trajectories), a sweep's
figures and best trials (sweep_summary), the smoothing and IDM studies' parts (control_report). RESULTS.md
reuses these tables and figures.
"""
