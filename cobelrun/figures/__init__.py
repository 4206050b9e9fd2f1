"""Paper-style plots. Functions take data frames and a matplotlib ``ax``, never live objects."""
