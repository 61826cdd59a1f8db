"""Products made from a finished results folder: plots and exported object models."""
