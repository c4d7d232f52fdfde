"""Tables and figures regenerated from run directories."""
