"""Matplotlib figures from results (optional extra ``slam2d[viz]``); no math lives here."""
