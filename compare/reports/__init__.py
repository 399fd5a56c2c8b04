"""flexforce.compare.reports: the HTML reports of a comparison (:mod:`.comparison`) and of a
diagnosis (:mod:`.diagnosis`), from the templates shipped beside them."""
