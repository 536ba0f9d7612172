"""report.html's sections, one module each (with its figures); `html.SECTIONS` puts them in order."""
