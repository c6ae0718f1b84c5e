# Entry point at the repository root; the workflow itself is workflow/Snakefile.
# (Rules of an included file are never the default target, hence the rule below.)


include: "workflow/Snakefile"


rule default:
    default_target: True
    input:
        rules.all.input,
