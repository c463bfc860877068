"""reports/RESULTS.md from reports/RESULTS.template.md, and its notebook pages: the writer (writer), the placeholder
language checked before any study is read (template), the notebook pages it links (pages), the studies it is
built from (selection), Table I across studies (headline) and the paper's comparisons on its cells (paper_claims),
the "Studies used" table (provenance), the regeneration command (command), its small PNGs (pngs), placeholders
over several studies (across) and computed comparisons quoted by its prose (comparisons).
"""
