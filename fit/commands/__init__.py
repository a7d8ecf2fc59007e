"""One module per command: `fit` (run a fit config), `synth` (synthetic captures), `inspect`
(look at a capture), `bench` (speed and accuracy tables). The CLI (`fit/cli.py`) calls them."""
