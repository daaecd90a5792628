"""The run's HTML report (:mod:`pipeline.report.page`, its sections), what it reads of the run
(:mod:`pipeline.report.run_data`), its pictures (:mod:`pipeline.report.figures`), inline SVG plots and the
tracking summary it shows."""
