"""The report: report.txt, and report.html built from its SECTIONS (one module each under sections/)."""
