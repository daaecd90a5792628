"""The run's HTML report (:mod:`pipeline.report.page`), its inline SVG plots and the tracking summary it shows."""
