"""Tools around memrl that are not part of training: the window bot (a stand-in driver)."""
