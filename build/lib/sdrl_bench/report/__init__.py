"""The report: tracking store -> tables, figures, Markdown and HTML (reads runs; never trains)."""
