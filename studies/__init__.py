"""The code of one study each (not part of the installed package): run from the checkout, e.g.
`python -m studies.stability --help`. README.md says how to rerun each study."""
