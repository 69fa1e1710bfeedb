"""Looking at a trained run: the web viewer (stdr-view, on viser) and videos (stdr-render).
`core` holds what both render, with no web code."""
