"""`python -m goi`: the goi command, so that `torchrun ... -m goi fit-field --distributed` works
(torchrun starts a module or a script, not a console script). The CLI lives in goi_cli."""
