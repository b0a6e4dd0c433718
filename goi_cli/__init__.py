"""goi's command line: parse options, call a stage, report. The work lives in `stages`."""
