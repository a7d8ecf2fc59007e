"""One module per command, each a function usable from Python (docs/commands.md): `fit` (and
multi-start beside it, `starts`), `render`, `synth`, `inspect`, `export`, `batch`. The command
line (`fit/cli.py`) parses options and calls them; `bench` is `fit.bench.run`."""
