"""reports/RESULTS.md from reports/RESULTS.template.md: the writer (writer), the placeholder
language checked before any study is read (template), the studies it is built from (selection),
the "Studies used" table (provenance), its small PNGs (pngs), placeholders over several studies
(across) and computed comparisons quoted by its prose (comparisons).
"""
