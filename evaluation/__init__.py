"""Measuring the method, never part of it: BOP datasets and results, pose errors as
bop_toolkit defines them plus ADD-sym, fates, tracking metrics, the front end's scores, the
oracle front end and the dataset runner. The estimator imports nothing from here."""
