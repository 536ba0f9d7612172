"""The report: report.txt, report.html with its sections and figures, and the numbers they show."""
