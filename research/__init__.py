"""Research scripts and experiments: not part of the installed `gmt` package (research/README.md)."""
