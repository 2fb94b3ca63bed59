"""The web console (``cell serve``): the operator's screen, the quality engineer's archive, a JSON API.

Another face on the same runner as the CLI: a job started here is ``cell run`` in a child process,
watched through its job folder and run log. See docs/decisions/0018-web-console.md.
"""
