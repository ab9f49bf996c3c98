from parjam.cli import entry

entry()
