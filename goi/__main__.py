from goi_cli.main import entry

entry()
