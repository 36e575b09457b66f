"""Reporting: evaluations and studies as Markdown tables (:mod:`~sfm_learn.reporting.tables`),
PNG plots (:mod:`~sfm_learn.reporting.plots`, the only matplotlib user of sfm_learn, imported
lazily) and the ``mkv demo`` report (:mod:`~sfm_learn.reporting.report`)."""
